"""Gradient-based gain tuning for fojax controllers."""
