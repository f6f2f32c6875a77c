"""services: the only package that knows Zenoh: wire messages, ROV and base-station loops, CLI wiring."""
