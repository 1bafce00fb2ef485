"""Dev-time converters and model writers (not installed with the package)."""
