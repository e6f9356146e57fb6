(cncjs-smoke: a 40 x 40 mm outline with 10 mm corners in two passes, then a 10 mm bore)
(tool: 3.175 mm flat end mill; stock top at Z0; the work zero is where the router starts)
G90 G94
G17
G21
N10 S12000 M3
N20 G0 Z5.
G0 X20. Y10.
(outline, pass 1)
G1 Z-1. F300.
X40. F600.
G3 X50. Y20. I0. J10.
G1 Y40.
G3 X40. Y50. I-10. J0.
G1 X20.
G3 X10. Y40. I0. J-10.
G1 Y20.
G3 X20. Y10. I10. J0.
(outline, pass 2)
G1 Z-2. F300.
X40. F600.
G3 X50. Y20. I0. J10.
G1 Y40.
G3 X40. Y50. I-10. J0.
G1 X20.
G3 X10. Y40. I0. J-10.
G1 Y20.
G3 X20. Y10. I10. J0.
G0 Z5.
(bore)
G0 X25. Y30.
G1 Z-1. F300.
G2 X25. Y30. I5. J0. F400.
G0 Z5.
N30 M5
G0 X60. Y55.
M30
