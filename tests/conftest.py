"""Suite-wide settings."""

import torch

# Simulator tests run worker processes beside the model on a 2-core machine; one intra-op thread
# avoids oversubscription, which made small networks about 10x slower there.
torch.set_num_threads(1)
