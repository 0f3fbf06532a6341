"""nerfbake: posed photographs to real-time radiance fields."""
__version__ = "0.1.0"
