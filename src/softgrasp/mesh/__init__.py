"""Tetrahedral meshes: the frozen :class:`TetMesh`, generators and file I/O."""

from softgrasp.mesh.generate import box, cylinder, sphere
from softgrasp.mesh.io import load_mesh, save_mesh
from softgrasp.mesh.tetmesh import TET_EDGES, TET_FACES, TetMesh, signed_volumes

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
