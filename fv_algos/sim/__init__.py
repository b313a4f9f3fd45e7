"""Simulated FingerVision sensor: skin, contact mechanics, objects, scenes, rendering, ground truth."""
