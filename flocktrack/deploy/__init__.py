"""Deploying a flock beyond one launcher: Docker Compose files and images, the secure mode's keys and ACL,
and the multi-router mesh."""
