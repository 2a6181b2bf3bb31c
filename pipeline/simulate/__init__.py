"""Simulators: feature-level scenes and recorded sessions in rooms."""
