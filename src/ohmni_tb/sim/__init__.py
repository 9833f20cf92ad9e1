"""Virtual firmware for every device on the Ohmni bus, and the simulated line."""
