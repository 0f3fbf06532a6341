"""The two teachers: a hash-grid SH field marched through an occupancy grid, and NeRF-SH with coarse-to-fine
sampling. Both return the same dictionary from :meth:`render_rays` (see the package docstring)."""
from __future__ import annotations

from dataclasses import dataclass, field as dc_field

import torch
from torch import nn

from nerfbake.fields.hash_sh import HashSHConfig, HashSHField
from nerfbake.fields.nerf_sh import NeRFSHConfig, NeRFSHField
from nerfbake.kernels.march import march_rays
from nerfbake.render.packed import packed_composite, packed_distortion_loss, packed_weights
from nerfbake.render.quadrature import composite, weights_from_density
from nerfbake.render.sampling import sample_pdf, stratified_t, uniform_t
from nerfbake.render.sh import eval_sh_color, sh_basis, sh_num_coeffs
from nerfbake.teacher.proposal import ProposalConfig, ProposalSampler, scale_gradients_by_distance, spacing
from nerfbake.teacher.sampling import OccupancyGrid, ray_box


@dataclass
class SceneBox:
    """Where the teacher spends its resolution; ``near``/``far`` clip rays (dataset bounds)."""

    box_min: list[float]
    box_max: list[float]
    near: float = 0.0
    far: float = 1e10
    contracted: bool = False
    # Rays leaving the box end on a colour the teacher learns from the ray direction (object-centred captures of
    # opaque photos, whose box holds the object and its surroundings but not the far background).
    learned_background: bool = False
    # A given box that holds the cameras (a Blender scene with ``aabb`` whose cameras stand inside it): an indoor
    # scene, whose walls lie inside the box. Contracted like any scene with cameras inside (rays still march on past
    # the box), but sampled by marching the grid (``unbounded_sampler`` auto).
    indoor: bool = False


class DirectionalBackground(nn.Module):
    """Colour at infinity as a function of direction alone: degree-4 SH basis -> 32 ReLU units -> sigmoid RGB. A
    distant background looks the same from every camera, so a direction is all it needs; anything nearer
    belongs in the box."""

    def __init__(self, degree: int = 4, hidden: int = 32):
        super().__init__()
        self.degree = degree
        self.net = nn.Sequential(nn.Linear(sh_num_coeffs(degree), hidden), nn.ReLU(), nn.Linear(hidden, 3))

    def forward(self, dirs: torch.Tensor) -> torch.Tensor:
        unit = dirs / dirs.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        return torch.sigmoid(self.net(sh_basis(self.degree, unit)))


@dataclass
class HashTeacherConfig:
    field: HashSHConfig = dc_field(default_factory=HashSHConfig)
    grid_resolution: int = 128
    render_steps: int = 512  # marching steps across the box diagonal (training)
    eval_step_scale: float = 0.5  # rendering without a generator marches finer: a better quadrature, +0.3 dB on lego
    alpha_thresh: float = 0.01
    grid_update_every: int = 16
    # Colour (the larger MLP and the SH sum) is evaluated only for samples whose compositing weight exceeds this:
    # on lego ~60% of marched samples sit behind the surface or in near-empty occupied cells and weigh < 1e-5.
    # Their colour would move a pixel by < 1e-5 each; density, and so every weight, still sees every sample.
    color_weight_thresh: float = 1e-5
    # The occupancy grid cannot prune before the field has learnt where empty space is: the first steps march
    # ~140 samples per ray through half the box (a minute of a 20-minute CPU budget). March this many times
    # coarser until ``coarse_march_steps``; the field is still a blur then, which the coarse steps resolve.
    coarse_march_scale: float = 4.0
    coarse_march_steps: int = 256
    # With a learned background the grid prunes nothing for this many steps. Early on the background explains
    # the average pixel and drains density everywhere; a grid that prunes then leaves most of the scene without
    # samples, to be regrown through hash collisions (textured orbit, recovered poses: occupancy 6.5% at step
    # 100, held-out 24.0 dB at 1000 steps; kept whole for 256 steps: see process_quality's figures).
    background_warmup_steps: int = 256
    # Unbounded (contracted) scenes: "proposal" samples with a proposal network (mip-NeRF 360: 64 proposal and 32
    # final samples a ray); "grid" marches an occupancy grid over contracted space with steps that grow as r^2
    # beyond the unit cube (kernels/march.py), with the distortion loss and near-camera gradient scaling of the
    # proposal path. The grid is not the default for real captures: a real scene's rays all end on a surface and the grid cannot skip
    # what lies behind it (fern after warm-up: 46 samples a ray kept for the gradient pass, 2.5k training rays/s
    # against the proposal path's 5.0k; benchmarks/unbounded_speed.py). "auto" (the default) marches the grid in
    # indoor scenes (SceneBox.indoor) and uses the proposal network elsewhere: in the synthetic house (seven rooms, 280
    # views, 600 steps) the proposal network left fog in front of the cameras of the two large bedrooms upstairs
    # (20.79 / 18.15 dB held-out there; trained alone they score 27.8 / 22.0), and marching scores 25.31 / 24.68 and
    # 26.75 dB over the whole walk against 24.56, at 5.4k training rays/s against 13.6k.
    unbounded_sampler: str = "auto"
    unbounded_far: float = 1000.0  # where contracted marching stops (scene units; cameras lie in [-1, 1]^3)
    # Real captures have no empty background: every ray ends on a surface, and the grid cannot skip what lies
    # behind it (~60 marched samples a ray on fern). Training renders of contracted scenes therefore first take
    # the density of every marched sample without gradients, then keep for the gradient pass only the samples
    # before the transmittance falls below ``early_stop_transmittance`` whose alpha reaches ``cull_alpha``
    # (nerfacc's estimator does the same); the composite of the kept samples differs from the full one by less
    # than those bounds.
    early_stop_transmittance: float = 1e-4
    cull_alpha: float = 1e-4
    proposal: ProposalConfig = dc_field(default_factory=ProposalConfig)  # unbounded scenes
    # The field's MLPs on unbounded scenes: "bfloat16" computes their CPU pass in bfloat16 where the CPU has native
    # bfloat16 matmuls (HashSHField.set_mlp_dtype). Measured on real captures only, so bounded scenes (lego's
    # figures) keep float32; teachers recorded before it read float32.
    unbounded_mlp_dtype: str = "float32"


@dataclass
class NeRFSHTeacherConfig:
    field: NeRFSHConfig = dc_field(default_factory=NeRFSHConfig)
    coarse_samples: int = 64
    fine_samples: int = 128
    sparsity_weight: float = 1e-3
    sparsity_length: float = 0.05
    sparsity_points: int = 10000


def _shade(field_out, dirs):
    sigma, sh = field_out
    return sigma, eval_sh_color(sh, dirs)


FIELD_CHUNK = 1 << 18  # samples the hash field evaluates at once where a pass needs no gradient


class HashTeacher(nn.Module):
    """Bounded scenes march through an occupancy grid; unbounded (contracted) ones use proposal sampling."""

    kind = "hash"

    def __init__(self, cfg: HashTeacherConfig, box: SceneBox):
        super().__init__()
        self.cfg, self.box = cfg, box
        self.field = HashSHField(cfg.field, box.box_min, box.box_max, contracted=box.contracted)
        if box.contracted:
            self.field.set_mlp_dtype(cfg.unbounded_mlp_dtype)
        size = torch.tensor(box.box_max) - torch.tensor(box.box_min)
        self.dt = float(size.norm()) / cfg.render_steps
        if self.uses_proposal:
            lo, hi = torch.tensor(box.box_min), torch.tensor(box.box_max)
            self.proposal = ProposalSampler(cfg.proposal, (lo + hi) / 2, (hi - lo) / 2)
        else:
            if box.contracted:  # the grid spans contracted space, twice the box: the same steps cover it
                self.dt = 2 * float(size.min()) * 3 ** 0.5 / cfg.render_steps
            self.grid = OccupancyGrid(box.box_min, box.box_max, cfg.grid_resolution, self.dt, cfg.alpha_thresh,
                                      contracted=box.contracted)
        self.train_dt = self.dt  # marching step of training renders (see before_step)
        self.background = DirectionalBackground() if box.learned_background else None

    @property
    def sh_degree(self) -> int:
        return self.field.sh_degree

    @property
    def uses_proposal(self) -> bool:
        sampler = self.cfg.unbounded_sampler
        return self.box.contracted and (sampler == "proposal" or (sampler == "auto" and not self.box.indoor))

    def query(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        return self.field(x)

    def density_at(self, x: torch.Tensor) -> torch.Tensor:
        """sigma at points as the renderer sees the scene: zero outside a bounded scene's box and in cells its
        occupancy grid skips (the field was never fitted there, so raw values in empty cells mean nothing)."""
        sigma = self.field.density(x)
        if self.uses_proposal:
            return sigma
        return torch.where(self.grid.occupied_at(x), sigma, torch.zeros_like(sigma))

    @torch.no_grad()
    def may_be_occupied(self, x: torch.Tensor) -> torch.Tensor:
        """Where the occupancy grid, grown by one cell, lets density be (all True on the proposal path, which keeps
        no grid)."""
        if self.uses_proposal:
            return torch.ones(x.shape[0], dtype=torch.bool, device=x.device)
        return self.grid.occupied_at(x.to(self.grid.occupied.device), dilate=1).to(x.device)

    def before_step(self, step: int, generator: torch.Generator) -> None:
        self.train_dt = self.dt * (self.cfg.coarse_march_scale if step < self.cfg.coarse_march_steps else 1.0)
        if not self.uses_proposal and step % self.cfg.grid_update_every == 0:
            warming_up = self.background is not None and step < self.cfg.background_warmup_steps
            self.grid.update(self.field.density, generator, prune=not warming_up)

    def after_training(self, generator: torch.Generator, log=None) -> None:
        """Once, when the last step is done: the occupancy grid the saved teacher renders with (see refresh)."""
        if not self.uses_proposal:
            if log is not None:
                log("final occupancy grid: re-evaluating every cell (~20 s on 2 cores)")
            self.grid.refresh(self.field.density, generator)

    @property
    def noise_dims(self) -> int:
        """Uniform random numbers one training ray consumes (drawn by the trainer for the whole global batch)."""
        return self.proposal.noise_dims if self.uses_proposal else 1

    def render_rays(self, origins, dirs, background=None, noise: torch.Tensor | None = None) -> dict:
        """``noise`` (R, noise_dims) in [0, 1) makes this a training render (jittered samples); None renders
        deterministically with the finer evaluation step. A teacher with a learned background uses it in place
        of ``background``."""
        if self.background is not None:
            background = self.background(dirs)
        if self.uses_proposal:
            return self._render_proposal(origins, dirs, background, noise)
        n = origins.shape[0]
        grid = self.grid
        if grid.contracted:
            t_near = torch.full((n,), float(self.box.near), device=origins.device)
            t_far = torch.full((n,), min(self.box.far, self.cfg.unbounded_far), device=origins.device)
            centre, half = grid.centre, grid.half
        else:
            t_near, t_far = ray_box(origins, dirs, grid.box_min, grid.box_max)
            t_near = t_near.clamp_min(self.box.near)
            t_far = t_far.clamp_max(self.box.far)
            centre = half = None
        offset = None if noise is None else noise[:, 0]
        dt = self.train_dt if noise is not None else self.dt * self.cfg.eval_step_scale
        ray_idx, t0, t1 = march_rays(origins, dirs, t_near, t_far, grid.occupied, grid.grid_min, grid.grid_max, dt,
                                     offset, contract_centre=centre, contract_half=half)
        contracted_training = grid.contracted and noise is not None  # culled, scaled, distortion-regularised
        if contracted_training:
            ray_idx, t0, t1 = self._cull(origins, dirs, ray_idx, t0, t1, n)
        mid = 0.5 * (t0 + t1)
        pts = origins[ray_idx] + mid[:, None] * dirs[ray_idx]
        field = self.field.density_and_features
        sigma, feat = field(pts) if noise is not None else self._in_chunks(field, pts)  # renders: in chunks
        if contracted_training:
            sigma, feat = scale_gradients_by_distance(mid, self.cfg.proposal.grad_scale_distance, sigma, feat)
        w, alpha = packed_weights(sigma, t0, t1, ray_idx, n)
        if grid.contracted and noise is None:
            # Rendered samples that the cull bounds make negligible are dropped from the output too: the march
            # goes on behind walls to unbounded_far (437 samples a ray on the house, 95 kept), and every caller
            # that renders a student on these intervals (distillation's views, the bake's alive voxels) would
            # carry them all. The weights of the kept samples are unchanged.
            keep = self._worth_a_pass(w, alpha)
            ray_idx, t0, t1, w, feat = ray_idx[keep], t0[keep], t1[keep], w[keep], feat[keep]
        seen = torch.nonzero(w.detach() > self.cfg.color_weight_thresh).squeeze(-1)
        rgb = torch.zeros(w.shape[0], 3, dtype=w.dtype, device=w.device)
        rgb = rgb.index_put((seen,), eval_sh_color(self.field.sh_coeffs(feat[seen]), dirs[ray_idx[seen]]))
        out = packed_composite(w, rgb, t0, t1, ray_idx, n, background)
        out.update(ray_idx=ray_idx, t0=t0, t1=t1, w=w, num_samples=ray_idx.numel())
        if contracted_training:
            out["_distortion"] = (spacing(t0), spacing(t1), w, ray_idx, n)
        return out

    @staticmethod
    def _in_chunks(fn, pts: torch.Tensor):
        """``fn`` (the field's density or density_and_features) over ``FIELD_CHUNK`` samples at a time, the results
        joined: a march can hold millions (8192 rays through the house's contracted grid: 3.6 M), and the
        encoding's and MLPs' temporaries of all of them at once were the largest allocation of a distillation's
        validation view and of the bake."""
        if pts.shape[0] <= FIELD_CHUNK:
            return fn(pts)
        parts = [fn(pts[s: s + FIELD_CHUNK]) for s in range(0, pts.shape[0], FIELD_CHUNK)]
        return tuple(map(torch.cat, zip(*parts))) if isinstance(parts[0], tuple) else torch.cat(parts)

    @torch.no_grad()
    def _cull(self, origins, dirs, ray_idx, t0, t1, n):
        """The marched samples worth a gradient pass (see ``early_stop_transmittance``)."""
        if not ray_idx.numel():
            return ray_idx, t0, t1
        pts = origins[ray_idx] + (0.5 * (t0 + t1))[:, None] * dirs[ray_idx]
        sigma = self._in_chunks(self.field.density, pts)
        keep = self._worth_a_pass(*packed_weights(sigma, t0, t1, ray_idx, n))
        return ray_idx[keep], t0[keep], t1[keep]

    def _worth_a_pass(self, w: torch.Tensor, alpha: torch.Tensor) -> torch.Tensor:
        """Indices of the samples before the transmittance falls below ``early_stop_transmittance`` whose alpha
        reaches ``cull_alpha``."""
        trans = w / alpha.clamp_min(1e-12)
        return torch.nonzero((trans > self.cfg.early_stop_transmittance) & (alpha >= self.cfg.cull_alpha)).squeeze(-1)

    def _render_proposal(self, origins, dirs, background, noise) -> dict:
        r = origins.shape[0]
        near = torch.full((r,), float(self.box.near), device=origins.device)
        s, t, proposal = self.proposal.sample(origins, dirs, near, noise)
        mid = 0.5 * (t[:, 1:] + t[:, :-1])
        pts = origins[:, None] + mid[..., None] * dirs[:, None]
        k = mid.shape[1]
        sigma, feat = self.field.density_and_features(pts.reshape(-1, 3))
        sigma, feat = scale_gradients_by_distance(mid.reshape(-1), self.cfg.proposal.grad_scale_distance, sigma, feat)
        w, _ = weights_from_density(sigma.view(r, k), t)
        seen = torch.nonzero(w.detach().reshape(-1) > self.cfg.color_weight_thresh).squeeze(-1)  # as the grid path
        rgb = torch.zeros(r * k, 3, dtype=w.dtype, device=w.device)
        rgb = rgb.index_put((seen,), eval_sh_color(self.field.sh_coeffs(feat[seen]), dirs[seen // k]))
        out = composite(w, rgb.view(r, k, 3), background, t)
        out.update(ray_idx=torch.arange(r, device=origins.device).repeat_interleave(k), t0=t[:, :-1].reshape(-1), t1=t[:, 1:].reshape(-1),
                   w=w.reshape(-1), num_samples=r * (k + self.proposal.proposal_samples))
        out["_proposal"] = (s, w, proposal)
        return out

    def extra_losses(self, out: dict, generator) -> dict[str, torch.Tensor]:
        if "_distortion" in out:
            return {"distortion": self.cfg.proposal.distortion_weight * packed_distortion_loss(*out["_distortion"])}
        if "_proposal" not in out:
            return {}
        s, w, proposal = out["_proposal"]
        return self.proposal.losses(s, w, proposal)


class NeRFSHTeacher(nn.Module):
    """Coarse and fine NeRF-SH MLPs; the fine pass evaluates coarse + importance samples (NeRF §5.2)."""

    kind = "nerf-sh"
    background = None  # no learned background: rays that leave the box take the caller's colour

    def __init__(self, cfg: NeRFSHTeacherConfig, box: SceneBox):
        super().__init__()
        self.cfg, self.box = cfg, box
        self.coarse = NeRFSHField(cfg.field)
        self.fine = NeRFSHField(cfg.field)

    @property
    def sh_degree(self) -> int:
        return self.fine.sh_degree

    @property
    def field(self) -> NeRFSHField:
        return self.fine

    def query(self, x):
        return self.fine(x)

    def density_at(self, x: torch.Tensor) -> torch.Tensor:
        """sigma at points, zero outside the scene box (where the renderer never samples)."""
        lo = torch.as_tensor(self.box.box_min, dtype=x.dtype, device=x.device)
        hi = torch.as_tensor(self.box.box_max, dtype=x.dtype, device=x.device)
        sigma = self.fine(x)[0]
        return torch.where(((x >= lo) & (x <= hi)).all(-1), sigma, torch.zeros_like(sigma))

    def may_be_occupied(self, x: torch.Tensor) -> torch.Tensor:
        """All True: NeRF-SH keeps no occupancy grid."""
        return torch.ones(x.shape[0], dtype=torch.bool, device=x.device)

    def before_step(self, step, generator) -> None:
        pass

    def after_training(self, generator, log=None) -> None:
        pass

    def _near_far(self, origins, dirs):
        dev = origins.device
        t_near, t_far = ray_box(origins, dirs, torch.tensor(self.box.box_min, device=dev), torch.tensor(self.box.box_max, device=dev))
        t_near = t_near.clamp_min(self.box.near)
        t_far = torch.maximum(t_far.clamp_max(self.box.far), t_near + 1e-3)
        return t_near, t_far

    def _pass(self, net, origins, dirs, t, background):
        mid = 0.5 * (t[:, 1:] + t[:, :-1])
        pts = origins[:, None] + mid[..., None] * dirs[:, None]
        s = mid.shape[1]
        sigma, rgb = _shade(net(pts.reshape(-1, 3)), dirs[:, None].expand(-1, s, -1).reshape(-1, 3))
        sigma, rgb = sigma.view(-1, s), rgb.view(-1, s, 3)
        w, _ = weights_from_density(sigma, t)
        return w, composite(w, rgb, background, t), sigma

    @property
    def noise_dims(self) -> int:
        return self.cfg.coarse_samples + 1 + self.cfg.fine_samples

    def render_rays(self, origins, dirs, background=None, noise: torch.Tensor | None = None) -> dict:
        t_near, t_far = self._near_far(origins, dirs)
        nc = self.cfg.coarse_samples
        t_c = stratified_t(t_near, t_far, nc, u=noise[:, : nc + 1]) if noise is not None else uniform_t(t_near, t_far, nc)
        w_c, out_c, _ = self._pass(self.coarse, origins, dirs, t_c, background)
        t_f = sample_pdf(t_c, w_c.detach(), self.cfg.fine_samples, deterministic=noise is None,
                         u=None if noise is None else noise[:, nc + 1:])
        t_all, _ = torch.sort(torch.cat([t_c, t_f], dim=-1), dim=-1)
        w, out, _ = self._pass(self.fine, origins, dirs, t_all, background)
        r, s = w.shape
        out.update(
            rgb_coarse=out_c["rgb"],
            ray_idx=torch.arange(r, device=origins.device).repeat_interleave(s), t0=t_all[:, :-1].reshape(-1), t1=t_all[:, 1:].reshape(-1),
            w=w.reshape(-1), num_samples=r * (s + nc),
        )
        return out

    def extra_losses(self, out: dict, generator) -> dict[str, torch.Tensor]:
        """The sparsity prior on random points in the box, and NeRF's coarse colour loss is added by the trainer."""
        cfg = self.cfg
        lo, hi = torch.tensor(self.box.box_min), torch.tensor(self.box.box_max)
        pts = (lo + (hi - lo) * torch.rand(cfg.sparsity_points, 3, generator=generator)).to(self.fine.sigma_head.weight.device)
        sigma = self.fine.density(pts)
        return {"sparsity": cfg.sparsity_weight * (1.0 - torch.exp(-cfg.sparsity_length * sigma).mean())}


def build_teacher(kind: str, cfg, box: SceneBox) -> nn.Module:
    if kind == "hash":
        return HashTeacher(cfg, box)
    if kind == "nerf-sh":
        return NeRFSHTeacher(cfg, box)
    raise ValueError(f"unknown teacher field {kind!r}; choose hash or nerf-sh")
