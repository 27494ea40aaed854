"""Datasets: episodes recorded from the simulator, stored and served for training.

- generate: scripted, play, program and policy episodes into MCAP files, a manifest and the training
  cache (`python -m sim_data.dataset.generate`, make data);
- episodes: the MCAP format of one episode (write, read, metadata);
- cache: the memory-mapped training cache built from the MCAP files, and the window loader;
- replay: an episode's recorded simulator state stepped again to check it (`python -m sim_data.dataset.replay`).
- lerobot: a dataset in LeRobot's layout v3.0 (`python -m sim_data.dataset.lerobot`, make export-lerobot).
"""
