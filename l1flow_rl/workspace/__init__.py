"""The application layer: building policies from configs, the training loop, checkpoints and reports."""
