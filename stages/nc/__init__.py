"""NC text: reading programs into blocks (:mod:`.reader`), splitting them into passes (:mod:`.moves`),
cutting via points (:mod:`.via`) and writing corrected programs (:mod:`.writer`, :mod:`.heidenhain`)."""
