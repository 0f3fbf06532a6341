"""Teachers: a field plus the sampler that renders it. Both later stages consume this one interface:

* ``teacher.query(x)`` -> ``sigma`` (N,), ``sh`` (N, 3*B)                    (octree building)
* ``teacher.render_rays(origins, dirs, background)`` -> per ray ``rgb`` (R,3), ``acc``, ``depth`` and the
  packed intervals ``ray_idx``, ``t0``, ``t1`` with their compositing weights ``w``  (SMERF distillation)
"""
