"""The public releases occtrain reads and writes in their own layouts and key names.

- :mod:`~occtrain.data.releases.nuscenes_tables`: the nuScenes v1.0 tables (``ROOT/<version>/*.json``)
  and the CAN bus expansion, read and checked (no nuscenes-devkit; its module docstring says why);
- :mod:`~occtrain.data.releases.nuscenes_import`: an Occ3D-layout dataset with occtrain's frame
  sidecars built from those tables and an Occ3D-nuScenes root (``occtrain data import nuscenes``);
- :mod:`~occtrain.data.releases.text_import`: OmniDrive-nuScenes, DriveLM and NuScenes-QA joined
  to a dataset's frames by sample token (``occtrain data import omnidrive|drivelm|nuscenes-qa``);
- :mod:`~occtrain.data.releases.nuscenes_export`: an occtrain dataset written back as those
  releases (``occtrain data export nuscenes``), so each importer is tested by a round trip.
"""
