"""Reading scene data from files: triangle meshes (needs ``trimesh``), glTF scenes (needs ``pygltflib``) and
hair strands (AMD TressFX ``.tfx`` and Cem Yuksel's ``.hair``, turned into curve segments by :func:`load_hair`).
"""

from jaxrt._src.io.gltf import GltfScene, load_gltf
from jaxrt._src.io.gltf_motion import GltfMotion, load_gltf_motion
from jaxrt._src.io.hair import HairCurves, load_hair, read_hair, read_tfx, write_hair
from jaxrt._src.io.meshes import load_mesh

__all__ = [
    "GltfMotion",
    "GltfScene",
    "HairCurves",
    "load_gltf",
    "load_gltf_motion",
    "load_hair",
    "load_mesh",
    "read_hair",
    "read_tfx",
    "write_hair",
]
