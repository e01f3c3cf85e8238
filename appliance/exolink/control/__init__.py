"""What motion is made of above the bus: the controller plugin interface (controller), what a
motion node knows of the watchdog (arming) and the operator's presence (holder)."""
