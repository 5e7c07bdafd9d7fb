"""Tetrahedral meshes: the frozen :class:`TetMesh`, generators and file I/O."""

from softgrasp.model.mesh.generate import box, cylinder, sphere
from softgrasp.model.mesh.io import load_mesh, save_mesh
from softgrasp.model.mesh.tetmesh import TET_EDGES, TET_FACES, TetMesh, signed_volumes

__all__ = [
    "TET_EDGES",
    "TET_FACES",
    "TetMesh",
    "box",
    "cylinder",
    "load_mesh",
    "save_mesh",
    "signed_volumes",
    "sphere",
]
