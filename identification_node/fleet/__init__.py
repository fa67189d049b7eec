"""Fleet identification: many bags of many robots, reduced per robot and period."""
