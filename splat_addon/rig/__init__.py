"""Splats that move with a rig: binding to an armature and posing, binding through a proxy mesh,
and collisions between splat objects over frames."""
