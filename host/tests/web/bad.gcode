; A program the page must refuse before it sends anything: line 4 does not fit the 39 bytes
; of a stored program line, even in its shortest form.
G1 X1 F1000
G1 X123.4567 Y123.4567 Z123.4567 E123.4567 F1234.5
G1 X2
