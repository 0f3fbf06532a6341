"""PlenOctrees (Yu et al. 2021): a sparse 2^3-tree with spherical-harmonic leaves in the svox layout.

Stages: :mod:`.build` (from a teacher), :mod:`.render` (Warp kernel + torch reference), :mod:`.optimize`
(fine-tuning with the analytic backward), :mod:`.compress` (median-cut quantisation), :mod:`.io` (svox/volrend
``.npz``), :mod:`.evaluate` (metrics and frame timing).
"""
