"""Simulation: segment worlds, exact ray casting, noisy odometry, scenarios."""
