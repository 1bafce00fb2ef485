"""Perception: masks, point clouds, segmentation, target detection, target occupancy, and
whether a camera's images have arrived (ImagesReady)."""
