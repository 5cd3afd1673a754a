"""Reading scene data from files: triangle meshes (:mod:`jaxrt._src.io.meshes`)."""

from jaxrt._src.io.meshes import load_mesh

__all__ = ["load_mesh"]
