"""The machined surface from global ordered scans (seed 000 claims 1, 4, 5, 7, 8): tiles and their
scans (:mod:`.tiles`, :mod:`.ordered`), which passes cut and where (:mod:`.cut_passes`), the
generating point of each predicted pass (:mod:`.strip`) and its cutting region (:mod:`.engagement`)."""
