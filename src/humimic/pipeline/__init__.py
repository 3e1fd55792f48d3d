"""What composes the parts: batch jobs and the sim-to-real loop."""
