"""Streaming a bag through the node's pipeline, validation on bags, and identify()."""
