"""The render chain's kernels: ordered scans over tiles, cutting passes, generating points and the
cutting region (seed 000 claims 1 and 4–8)."""
