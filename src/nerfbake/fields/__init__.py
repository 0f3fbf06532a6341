"""Trainable fields: encodings (positional, hash grid), the NeRF-SH MLP and the hash-grid SH field.

A field maps world points (N, 3) to density ``sigma`` (N,) >= 0 and colour coefficients ``sh`` (N, 3*B)
in the svox layout (colour = sigmoid(sum_k Y_k(d) c_k), see :mod:`nerfbake.render.sh`).
"""
