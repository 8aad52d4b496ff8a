"""Identification by linear regression: the equations, their solution, the effect search."""
