"""Shipped presets: one TOML file per preset, validated by kbbatch.presets."""
