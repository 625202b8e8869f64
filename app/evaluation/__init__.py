"""Accuracy measurements on the real recordings, split by walk, never by sample."""
