"""The controllers that learn the plant from data alone: no plant equations
(the import contract "learned-no-equations" in pyproject.toml)."""
