"""Fine-tuning a trained BC policy with rewards: the algorithms and their acting modules."""
