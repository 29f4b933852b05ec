"""Headless OpenGL rendering of the worlds (RGB, depth, instance ids)."""
