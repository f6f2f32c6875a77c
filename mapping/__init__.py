"""mapping: NED clouds, Open3D plane extraction and the shared plane map (knows nothing of Zenoh)."""
