"""Packaged data: the pelvis model file and its NOTICE (attribution of the atlas it comes from)."""
