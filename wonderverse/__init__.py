"""WonderVerse: text prompt -> extendable 3D scene.

The library holds plain functions over arrays; orchestration lives in `tasks/` and `flows/`.
"""

__version__ = "0.1.0"

# Bumped whenever the scene-store layout changes incompatibly; a store written by a newer
# format is refused rather than misread.
STORE_FORMAT = 1
