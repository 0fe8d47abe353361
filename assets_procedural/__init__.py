"""assets_procedural package."""
