"""The lowest layer: the process's runtime settings (64-bit floats, the CPU platform, the
compile cache, XLA flags), the model files' location, users' own files, batch chunking."""
