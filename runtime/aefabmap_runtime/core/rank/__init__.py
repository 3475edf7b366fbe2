"""Rank: the places a frame may show, by FAB-MAP 2.0 over the Chow-Liu tree (or tf-idf BoW)."""
