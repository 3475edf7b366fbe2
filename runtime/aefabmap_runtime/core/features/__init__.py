"""Extract: local features (keypoints and descriptors) of one image, per registered kind."""
