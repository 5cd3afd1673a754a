"""Ray/primitive tests, one module per primitive. They know nothing of BVHs."""
