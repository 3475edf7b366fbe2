"""Records with a fixed shape: the wire messages and their JSON schemas, the map state as arrays."""
