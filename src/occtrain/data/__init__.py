"""Datasets: the Occ3D layout, the synthetic world, webdataset shards and datamodules."""
