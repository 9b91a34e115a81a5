"""Particle location from decoded light fields."""
