"""The user's steps as library calls (each CLI command calls one of these)."""
