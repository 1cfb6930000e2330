"""Training: losses, the loop (train/finetune), evaluation and checkpoints."""
