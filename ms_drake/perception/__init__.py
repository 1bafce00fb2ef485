"""Perception: masks, point clouds, (later) segmentation, target detection, occupancy."""
