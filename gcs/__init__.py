"""triswarm.gcs."""
