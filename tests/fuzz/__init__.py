"""The fuzz corpus (#27): hostile inputs per surface, each with its expected outcome class (`corpus.Case`);
`tests/test_fuzz_corpus.py` runs them."""
