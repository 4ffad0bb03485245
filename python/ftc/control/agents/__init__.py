"""The controllers, one module per method family, each with the options it
reads. ``learned/`` holds those that learn the plant and use no plant
equations; ``physics/`` those that plan on the plant's equations."""
