"""Mesh utilities: split a scene mesh into objects, sample surfaces, export meshes and point clouds."""

from torm.mesh.export import write_mesh, write_point_cloud
from torm.mesh.sample import sample_objects, sample_surface
from torm.mesh.split import split_components

__all__ = ["split_components", "sample_surface", "sample_objects", "write_mesh", "write_point_cloud"]
