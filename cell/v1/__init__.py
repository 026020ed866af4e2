"""Generated protobuf code for the bus messages (from proto/cell/v1; regenerate with `make proto`)."""
