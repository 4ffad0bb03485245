"""The controllers that plan on the plant's equations (true or identified)."""
