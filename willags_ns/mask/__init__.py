"""The transient mask: EMA teacher, perceptual distance and threshold, the step's mask, its SfM safeguard and its
health watch."""
