' eyetohand calibration collection for Epson robots (SPEL+, RC700/RC90 with EPSON RC+ 7).
' UNTESTED: no Epson controller here. Read examples/robots/README.md first.
'
' Vision side: eyetohand serve --tcp 0.0.0.0:5000 --camera URI
' Controller set-up (EPSON RC+: Setup > System Configuration > Controller > TCP/IP), port #201:
'   IP address = the vision PC, TCP/IP port = 5000, Terminate = LF, Protocol = TCP
'   (the SetNet line below sets the same from the program).
'
' Traps handled here:
' * Print # ends every line with the port's terminator; Line Input # reads up to it. The server
'   accepts LF or CR LF and answers LF, so Terminate must be LF: with CRLF, Line Input # would wait
'   for a CR LF that never comes. A CR left at the end of a reply (a server answering CR LF) is
'   stripped below.
' * Line Input # has no timeout of its own: ChkNet polls the bytes waiting, with our own 30 s limit.
' * Str$ gives about 7 significant digits (0.001 mm at 612.345 mm). Never send Print # a number list
'   with "," separators between items: SPEL+ inserts spaces; we build one string.
' * Go/Move end on the point (CP off) and Wait settles before the two grabs.

Global String gReply$
Global Real gVal(10)
Global Integer gCount

Function CalCollect
    String fields$(10)
    Real x, y, z
    Integer n

    SetNet #201, "192.168.0.10", 5000, LF, NONE, 0
    OpenNet #201 As Client
    WaitNet #201, 10
    If TW Then
        Print "eyetohand: cannot connect to the vision PC"
        Exit Function
    EndIf

    If Not Cmd("CAL BEGIN cell1,grid:5x5,-40,570,60,650,150") Then GoTo Fail

    Do
        If Not Cmd("CAL NEXT") Then GoTo Fail
        If gReply$ = "OK DONE" Then Exit Do
        If gCount <> 3 Then GoTo Fail
        x = gVal(0): y = gVal(1): z = gVal(2)
        Move XY(x, y, z, CU(Here)) CP Off   ' keep the current tool angle U
        Wait 0.5
        If Not Cmd("CAL POINT " + Fmt$(x) + "," + Fmt$(y) + "," + Fmt$(z)) Then
            If InStr(gReply$, "ERR moving") = 1 Then
                Wait 1.0
                If Not Cmd("CAL POINT " + Fmt$(x) + "," + Fmt$(y) + "," + Fmt$(z)) Then
                    Print "eyetohand: point skipped: ", gReply$
                EndIf
            Else
                Print "eyetohand: point skipped: ", gReply$
            EndIf
        EndIf
    Loop

    If Not Cmd("CAL END") Then GoTo Fail
    Print "eyetohand: calibrated: ", gReply$
    CloseNet #201
    Exit Function
Fail:
    Print "eyetohand: stopped: ", gReply$
    CloseNet #201
Fend

' Send one command, read one reply line into gReply$; OK replies' numbers into gVal(), gCount.
Function Cmd(line$ As String) As Boolean
    Integer i, t0
    String tok$(10)
    Print #201, line$
    t0 = 0
    Do While ChkNet(201) <= 0
        Wait 0.05
        t0 = t0 + 1
        If t0 > 600 Then        ' 30 s
            gReply$ = "ERR timeout waiting for the vision PC"
            Cmd = False
            Exit Function
        EndIf
        If ChkNet(201) < 0 Then
            gReply$ = "ERR connection lost"
            Cmd = False
            Exit Function
        EndIf
    Loop
    Line Input #201, gReply$
    If Right$(gReply$, 1) = Chr$(13) Then gReply$ = Left$(gReply$, Len(gReply$) - 1)
    gCount = 0
    If Left$(gReply$, 2) <> "OK" Then
        Cmd = False
        Exit Function
    EndIf
    If Len(gReply$) > 3 And gReply$ <> "OK DONE" Then
        gCount = ParseStr(Mid$(gReply$, 4), tok$(), ",")
        For i = 0 To gCount - 1
            gVal(i) = Val(tok$(i))
        Next i
    EndIf
    Cmd = True
Fend

' A number as text with a "." decimal point and 4 decimals.
Function Fmt$(v As Real) As String
    Fmt$ = FmtStr$(v, "0.0000")
Fend
