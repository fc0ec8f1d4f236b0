"""triswarm.companion."""
