"""Decide: which candidates are checked in what order, and evidence over frames (sequence, temporal)."""
