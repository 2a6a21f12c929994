"""Labelled feedback: frames to the evidence a profile version records (`evidence`), and the
health document built from its stored rows (`health_document`)."""
