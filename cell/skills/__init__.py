"""Skill servers and their clients: the AdeptServer-style ASCII protocol over TCP."""
