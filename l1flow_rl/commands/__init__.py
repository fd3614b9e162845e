"""The ``l1flow-rl`` command (``cli``) and the entry point of each of its sub-commands."""
