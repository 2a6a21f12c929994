"""Pydantic request/response models (OpenAPI schema with examples)."""
