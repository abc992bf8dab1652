"""``safenav bench {env,update,latency}``: the benchmarks whose figures the README quotes."""
