"""Volume-rendering math shared by every stage: quadrature, SH basis, contraction, sampling.

Names and shapes used throughout (after camp_zipnerf's stepfun):
  ``t``  (..., S+1) interval endpoints along a ray, in world distance (directions are unit length);
  ``sigma`` (..., S) density per interval; ``alpha`` (..., S) opacity per interval;
  ``w``  (..., S) compositing weights, ``sum(w) <= 1``; ``rgb`` (..., S, 3) colour per interval.
"""
from nerfbake.render.quadrature import (
    alpha_from_density,
    transmittance_from_alpha,
    weights_from_alpha,
    weights_from_density,
    composite,
)
from nerfbake.render.sh import sh_basis, sh_num_coeffs, eval_sh_color
from nerfbake.render.contraction import contract, uncontract
from nerfbake.render.sampling import uniform_t, stratified_t, sample_pdf, midpoints

__all__ = [
    "alpha_from_density", "transmittance_from_alpha", "weights_from_alpha", "weights_from_density", "composite",
    "sh_basis", "sh_num_coeffs", "eval_sh_color", "contract", "uncontract",
    "uniform_t", "stratified_t", "sample_pdf", "midpoints",
]
