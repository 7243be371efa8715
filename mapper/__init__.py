"""The mapper process."""
