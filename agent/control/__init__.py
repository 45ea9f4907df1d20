"""Sensor motion controllers (pure numpy)."""
