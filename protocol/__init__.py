"""triswarm.protocol."""
