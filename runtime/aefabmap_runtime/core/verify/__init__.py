"""Verify: two-view geometry between a frame and a place, judged a contrario."""
