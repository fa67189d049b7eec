"""Batch identification of a whole bag: samples, filtered rows, periodic averaging, the solve."""
