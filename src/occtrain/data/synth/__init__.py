"""The embedded synthetic driving world, in Occ3D-nuScenes geometry.

``generate_scene(name, seed, num_frames)`` builds one scene deterministically from its
seed: a grid city (roads, sidewalks, buildings, vegetation, parking, construction), traffic
and pedestrians simulated at 10 Hz, an ego route with turns, lane changes, stops and speed
changes, and per-frame annotations at 2 Hz. ``SyntheticScene.render(i)`` rasterises frame
``i`` with its lidar and camera visibility masks; ``prepare_sensors`` computes the
per-process sensor geometry up front. Modules: ``grid`` (vertical convention),
``catalog`` (object kinds, tracks), ``roads`` (network, lights, routes), ``citymap``
(static raster and objects), ``population`` and ``traffic`` (agents and their motion),
``raster`` (voxels, masks), ``annotate`` (FrameAnnotation), ``road_context`` (what a map
and a tracker would say of the route ahead: its points, the lead, the stop line, the
command), ``scene`` (the whole);
``text`` writes the captions, narrations and questions.
"""

from occtrain.data.synth.scene import SyntheticScene, generate_scene, prepare_sensors

__all__ = ["SyntheticScene", "generate_scene", "prepare_sensors"]
