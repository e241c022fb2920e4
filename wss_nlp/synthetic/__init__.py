"""Phantoms with exact truth: 2D slices, pulsatile flow, scanner-style exports, 4D flow vessels."""
