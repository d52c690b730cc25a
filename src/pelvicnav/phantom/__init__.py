"""Simulation: CT synthesis, dislocations, radiographs (the test bench with ground truth)."""
