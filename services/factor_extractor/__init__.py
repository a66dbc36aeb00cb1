"""factor-extractor: frames in, slot factors out as transitions (Dyn-O, chapter 7)."""
