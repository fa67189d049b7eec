"""Simulated arms: motion, dynamics and sensor noise for bags and tests."""
