"""Configuration presets shipped with gainfpn (YAML package data)."""
