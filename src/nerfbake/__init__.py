"""nerfbake: posed photographs to real-time radiance fields."""
import os

__version__ = "0.1.0"

# oneDNN (PyTorch's CPU matmuls) caches a compiled primitive for every matrix shape it meets, 1024 by default. The
# teachers' MLPs see a new row count nearly every call (the marcher's sample counts vary), so that cache grew the
# house's distillation by ~2.3 MB a second (0.35 GB of its 1.94 GB peak after 150 steps). 64 keeps the fixed-size
# chunks' primitives and drops the odd tails. Read at oneDNN's first matmul; a user's own setting wins.
os.environ.setdefault("ONEDNN_PRIMITIVE_CACHE_CAPACITY", "64")
