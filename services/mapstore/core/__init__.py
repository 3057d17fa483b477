"""Pure math of the map: arrays in, arrays out; no I/O, no transport, no storage."""
