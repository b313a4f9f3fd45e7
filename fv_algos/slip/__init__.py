"""Slip detection on displacement-field windows: models (models), a classical detector
(classical), windowing/splits/storage (windows), training (train), evaluation (evaluate) and
inference for the slip_detector node (classifier)."""
