"""`dpmhw render`: render one frame of a scene."""
