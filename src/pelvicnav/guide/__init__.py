"""Intraoperative guidance: residual motion to the planned target, overlays."""
