"""Pure parts of the query gateway: text embedding, answer shaping, PLY and TUM writers, poses per stream."""
