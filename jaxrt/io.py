"""Reading scene data from files (triangle meshes; needs the ``trimesh`` package)."""

from jaxrt._src.io.meshes import load_mesh

__all__ = ["load_mesh"]
