"""The map: places, their words and keypoints, the insertion queue, caps and eviction."""
