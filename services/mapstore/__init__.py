"""mapstore: the durable, keyframe-anchored semantic point map (see README.md)."""
