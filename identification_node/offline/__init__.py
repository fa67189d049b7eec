"""Identification of recorded bags: batch and replay, validation, reports, fleet."""
