"""svorf package."""
