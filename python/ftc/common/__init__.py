"""What every room of the package shares: atomic file writes, config
dataclasses turned into command lines with declared constraints, errors and
exit codes, named constants, build locations. Imports nothing else of ftc."""
