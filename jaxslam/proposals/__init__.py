"""Proposal distributions of the RBPF: odometry (OP), scan matching (SMP), look-ahead (LP)."""
