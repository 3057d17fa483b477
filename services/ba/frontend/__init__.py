"""BA frontend: keyframe graph and sliding window around the dense BA core (pure: arrays in, arrays out)."""
