"""A teacher run folder as an artifact: its layout (``config.json`` beside ``checkpoint.pt``) and its loader.

The routes (octree build, distillation, baking, evaluation) read teachers through this module, never through the
trainer (``teacher/train.py``), so reading a run does not pull in training code.
"""
from __future__ import annotations

import json
from pathlib import Path

from nerfbake.errors import RunFolderError, read_folder_config, reading
from nerfbake.fields.hash_sh import HashSHConfig
from nerfbake.fields.nerf_sh import NeRFSHConfig
from nerfbake.teacher.models import HashTeacherConfig, NeRFSHTeacherConfig, SceneBox, build_teacher
from nerfbake.teacher.presets import TeacherTrainConfig
from nerfbake.teacher.proposal import ProposalConfig
from nerfbake.train.loop import RUN_CONFIG, default_device, load_checkpoint

CHECKPOINT = "checkpoint.pt"
CONFIG = RUN_CONFIG


def config_from_dict(d: dict) -> TeacherTrainConfig:
    d = dict(d)
    h, n = d.pop("hash"), d.pop("nerf_sh")
    if "proposal" in h:
        h["proposal"].setdefault("stratified", False)  # runs made before the stratified draw
    prop = ProposalConfig(**h.pop("proposal")) if "proposal" in h else ProposalConfig()
    h.setdefault("unbounded_sampler", "proposal")  # runs made before the contracted occupancy grid
    d.setdefault("appearance", "none")  # runs made before per-image appearance
    d.setdefault("normalize", "auto")  # runs made before --normalize
    hash_cfg = HashTeacherConfig(field=HashSHConfig(**h.pop("field")), proposal=prop, **h)
    nerf_cfg = NeRFSHTeacherConfig(field=NeRFSHConfig(**n.pop("field")), **n)
    return TeacherTrainConfig(hash=hash_cfg, nerf_sh=nerf_cfg, **d)


def config_from_file(path: str | Path):
    """The teacher training config in a JSON file: a run's ``config.json`` (its ``"train"`` entry) or a bare config."""
    with reading(path, RunFolderError, "pass a run's config.json or a teacher training config written as JSON"):
        d = json.loads(Path(path).read_text())
        return config_from_dict(d.get("train", d))


def load_teacher(run: Path):
    """(teacher, config, dataset root, checkpoint state) from a run folder, with clear errors."""
    run = Path(run)
    cfg_path = run / CONFIG
    meta = read_folder_config(run, CONFIG, "teacher run folder", "nerfbake teacher train", lambda m: "train" in m)
    with reading(cfg_path, RunFolderError, "retrain with this version, or pass the --out folder of nerfbake teacher train"):
        cfg = config_from_dict(meta["train"])
        box = SceneBox(**meta["box"])
        model = build_teacher(cfg.field, cfg.model_config, box)
    state = load_checkpoint(run / CHECKPOINT)
    try:
        model.load_state_dict(state["model"])
    except (RuntimeError, KeyError, TypeError) as exc:
        first = str(exc).splitlines()[0]
        raise RunFolderError(f"{run / CHECKPOINT}: does not match {cfg_path} ({first}); retrain or restore the pair") from None
    model.to(default_device()).eval()
    return model, cfg, meta, state
