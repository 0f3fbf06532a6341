"""3D Gaussian splats: a nerfbake scene as the Gaussians that splat viewers, editors and engines open.

``gaussians.py`` holds the Gaussians in the 3DGS reference code's parameterisation; ``from_tree.py`` fits them to a
PlenOctree's leaves; ``io.py`` writes (and reads back) the reference ``.ply`` layout and the compact ``.splat``.
"""
