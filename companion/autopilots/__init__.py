"""The autopilot seam: what the companion needs of a kind of flight controller, one module per kind
(``base.Autopilot``; ``registry`` picks one from the flight controller's HEARTBEAT, or configuration
forces one). The loop, the protocol and the RFL never learn which autopilot flies."""
