"""The task ports against their references: throughput, profiles, parity, MetaWorld dynamics."""
