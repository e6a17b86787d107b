"""Physical descriptions of materials (the material table) used by the model and the simulator."""
