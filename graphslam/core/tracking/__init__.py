"""Online tracking on a radio map: access-point path-loss models, EKF/UKF fusion (Papers 000/002),
offline RTS / whole-run MAP smoothers."""
