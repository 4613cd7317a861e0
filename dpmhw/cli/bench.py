"""`dpmhw bench …`: benchmarks."""
