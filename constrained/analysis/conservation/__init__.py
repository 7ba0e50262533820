"""Conserved quantities found from the symmetries of a system (rigid motions of space)."""
