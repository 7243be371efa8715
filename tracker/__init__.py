"""The tracker process."""
