"""Rendering: images to per-pin stimulus parameters (issue 5). Imports cv2 lazily."""
