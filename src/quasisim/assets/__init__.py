"""Hand and object assets."""
