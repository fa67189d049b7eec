"""The wire: sensor_msgs/JointState CDR decoded and encoded (``cdr``) and the record it is
decoded into (``records``)."""
