"""Every ``nerfbake`` command as a dataclass (its options) with a ``run()`` (its call into the library): the layer
between the library and the command line. cli.py builds the parser from ``COMMANDS``; ``GROUPS`` names the commands
that share a first word. The library modules are imported inside ``run()``, so ``nerfbake --help`` starts at once."""
from __future__ import annotations

from nerfbake.commands.data import DataInfo, Metrics, Process, Synth
from nerfbake.commands.export import Export
from nerfbake.commands.octree import OctreeBuild, OctreeCompress, OctreeEval, OctreeInfo, OctreeOptimize, OctreeRender
from nerfbake.commands.runs import Demo, Doctor, Pipeline, Report, View
from nerfbake.commands.smerf import Bake, Distill, SmerfEval, SmerfInfo, SmerfRender
from nerfbake.commands.spec import Command
from nerfbake.commands.teacher import TeacherEval, TeacherRender, TeacherTrain

COMMANDS: tuple[type[Command], ...] = (
    DataInfo, Metrics, Synth, Process, TeacherTrain, TeacherEval, TeacherRender, OctreeBuild, OctreeOptimize,
    OctreeCompress, OctreeEval, OctreeInfo, OctreeRender, SmerfInfo, SmerfEval, SmerfRender, Distill, Bake, Export,
    View, Pipeline, Doctor, Report, Demo)
GROUPS = {"data": "inspect datasets", "teacher": "train, evaluate and render teacher fields",
          "octree": "PlenOctrees: build, fine-tune, compress, evaluate, render",
          "smerf": "SMERF baked scenes: inspect and render asset directories"}
