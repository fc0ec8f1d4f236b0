"""triswarm.sitl."""
