"""One reader per demonstration format; ``l1flow_rl.data.loading`` picks the one a path needs."""
