"""Reading scene data from files: triangle meshes (needs ``trimesh``) and glTF scenes (needs ``pygltflib``)."""

from jaxrt._src.io.gltf import GltfScene, load_gltf
from jaxrt._src.io.meshes import load_mesh

__all__ = ["GltfScene", "load_gltf", "load_mesh"]
