"""Loop closure: keyframe database, geometric verification, pose graph, loop closer."""
