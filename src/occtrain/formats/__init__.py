"""File formats occtrain reads and writes: atomic writes and safe loading, the safetensors + JSON
exports that hand a stage to the next, Occ3D's grid and classes, NuScenes-QA's question kinds."""
