"""bags package."""
