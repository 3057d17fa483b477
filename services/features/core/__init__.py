"""Pure math of the features service: arrays and tensors in and out, no transport, no files."""
