"""``python -m eval``: compare policies on seeded episodes of one scenario."""
