"""One update against its reference (mostly PyTorch): SAC, reward, world model, MRN, entropy."""
