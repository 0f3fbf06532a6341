"""The clearance around the training cameras: the space a teacher's rays never reached, emptied for the bakers."""
import numpy as np
import torch

from nerfbake.data.formats import load_dataset
from nerfbake.teacher.clearance import CameraClearance
from nerfbake.teacher.run import load_teacher


def test_clearance_is_the_union_of_balls_around_the_cameras():
    gen = np.random.default_rng(0)
    origins = gen.uniform(-1, 1, (37, 3))
    x = torch.from_numpy(gen.uniform(-2, 2, (5000, 3)).astype(np.float32))
    clearance = CameraClearance(origins, 0.25, chunk=777)  # several chunks
    want = np.linalg.norm(x.numpy()[:, None] - origins[None], axis=-1).min(1) <= 0.25
    got = clearance.inside(x).numpy()
    assert 0 < want.sum() < len(want)
    assert (got == want).all()
    assert not CameraClearance(origins, 0.0).inside(x).any()


def test_a_teachers_clearance_is_its_near_bound_around_its_training_cameras(rooms_teacher):
    teacher, _, meta, _ = load_teacher(rooms_teacher)
    cams = load_dataset(meta["data"]).cameras("train")
    clearance = CameraClearance.of_teacher(meta, cams)
    assert clearance.radius == meta["box"]["near"] > 0
    # points on a sphere of 0.9 x near around each camera are cleared; the teacher's density elsewhere is untouched
    gen = torch.Generator().manual_seed(0)
    u = torch.nn.functional.normalize(torch.randn(len(cams), 3, generator=gen), dim=-1)
    close = torch.from_numpy(np.stack([c.origin for c in cams])).float() + 0.9 * clearance.radius * u
    far = torch.rand(2000, 3, generator=gen) * 2 - 1
    far = far[~clearance.inside(far)]
    assert (clearance.density(teacher, close) == 0).all()
    assert torch.equal(clearance.density(teacher, far), teacher.density_at(far))
