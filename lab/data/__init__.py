"""Scenes and datasets: synthetic generators with exact ground truth, loaders for real data.

A dataset loader is a function with keyword-only options that returns a
:class:`lab.core.Loaded` (the initial state and, separately, its truth).
"""
