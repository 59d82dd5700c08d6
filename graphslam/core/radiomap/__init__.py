"""Fingerprints (eq. 9), radio maps and fingerprint search (exact and IVF kNN)."""
