"""Payload identification: change detection, the one-body fit, delivery."""
