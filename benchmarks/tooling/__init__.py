"""Device tooling: what a lent GPU machine lacks, packed to carry."""
