"""Human preference labelling: a query folder, a local web app that shows each query's two
clips and records a person's answers, and the mapping of answers to B-Pref labels."""
