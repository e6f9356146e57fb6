; The web page's end-to-end test program: a 60 mm square and a circle inside it, printed on
; the simulator's printer (relative extrusion; the simulator extrudes cold). About 17 s of
; virtual time: long enough to pause and resume it while it runs.
G21
G90
M83
G0 Z0.3 F600
G0 X40 Y40 F6000
G1 X100 Y40 E3 F1500
G1 X100 Y100 E3
G1 X40 Y100 E3
G1 X40 Y40 E3
G0 X70 Y50
G3 X70 Y50 I0 J20 E6 F1500 ; a full circle
G0 Z5 F600
G0 X10 Y10 F6000
