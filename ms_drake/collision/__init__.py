"""Learned collision checking (Ch. 6): SceneCollisionNet (scene_net)."""
