"""Digitally reconstructed radiographs: bone volume models and a batched forward projector."""
