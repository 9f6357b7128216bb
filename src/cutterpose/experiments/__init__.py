"""Experiments of the seed paper: the synthetic sweep (Fig. 5) and the image table (Table 2)."""
