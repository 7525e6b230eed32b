"""``synthetic_mini``: procedural driving scenes in the NuScenes-GSQA layout (``pipelines/data/layout.py``).

``pipelines.data.synth.build.build(SynthConfig(), root)`` renders seeded scenes (road, lanes,
vehicles, pedestrians, buildings, trees) for 6 surround cameras in several weathers, with depth,
LiDAR, ego poses, 3D/2D boxes and QA of every task family whose answers come from that ground
truth. ``build`` is deliberately not re-exported here: the package attribute would shadow the
``build`` module and break the dotted builder path ``pipelines.data.synth.build.build``.
"""

from pipelines.data.synth.config import SynthConfig

__all__ = ["SynthConfig"]
