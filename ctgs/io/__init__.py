"""File I/O helpers shared by the stages (images, downloads)."""
