"""3D-2D registration: CMA-ES driver, stage 1 (one bone vs the system geometry), stage 2."""
