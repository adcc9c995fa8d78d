"""visca package."""
