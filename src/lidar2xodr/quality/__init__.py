"""What `check` runs besides the ASAM checker: independent readers of the map and lane-width findings."""
