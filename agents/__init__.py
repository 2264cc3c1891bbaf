"""hilswarm agents: what one agent process is made of (link, pins, devices, vehicle, control)."""
