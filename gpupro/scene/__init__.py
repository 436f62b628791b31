"""Scene model: cameras, meshes, materials, lights, loaders and procedural scenes."""

from gpupro.scene.camera import Camera, make_camera
from gpupro.scene.lights import CAPSULE, DIRECTIONAL, POINT, SPOT, Lights, make_lights, no_lights, point_lights
from gpupro.scene.materials import Materials, make_materials
from gpupro.scene.mesh import Mesh, MeshError, concatenate_meshes, make_mesh
from gpupro.scene.scene import Scene
from gpupro.scene.sectors import Sectors, make_sectors
from gpupro.scene.light_generators import along_path, uniform_in_box
from gpupro.scene.loaders import load_mesh, load_scene
from gpupro.scene.procedural import SCENES, by_name, primitive_mesh
from gpupro.scene.validate import check_scene
