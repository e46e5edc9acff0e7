' eyetohand calibration collection for Epson robots (SPEL+, RC700/RC90 with EPSON RC+ 7).
' UNTESTED on a controller: no Epson controller here (its exchange with the real server is replayed
' by tests/test_robot_programs.py). Read examples/robots/README.md first.
'
' Vision side: eyetohand serve --tcp 0.0.0.0:5000 --camera URI --token-file FILE
' The token: a service on any address but loopback needs one (serve --token-file FILE or
' EYETOHAND_TOKEN) and the first line is then AUTH <token>: set token$ below, beside the address and
' port, to the same text (a server without a token answers AUTH with OK too). A wrong token is
' answered "ERR send 'AUTH <token>' first; closing" (code -14): the program stops and says so.
' Controller set-up (EPSON RC+: Setup > System Configuration > Controller > TCP/IP), port #201:
'   IP address = the vision PC, TCP/IP port = 5000, Terminate = LF, Protocol = TCP
'   (the SetNet line below sets the same from the program).
'
' Manual references: "EPSON RC+ 7.0 SPEL+ Language Reference", by statement/function name
' (SetNet, OpenNet, WaitNet, TW, ChkNet, Print #, Line Input #, CloseNet, CP, Move, Here, point
' expressions with :X :Y :Z, Wait, ParseStr, Val, FmtStr$, InStr, Left$, Right$, Mid$, Len).
'
' Traps handled here:
' * Print # ends every line with the port's terminator; Line Input # reads up to it. The server
'   accepts LF or CR LF and answers LF, so Terminate must be LF: with CRLF, Line Input # would wait
'   for a CR LF that never comes. A CR left at the end of a reply (a server answering CR LF) is
'   stripped below.
' * Line Input # has no timeout of its own: ChkNet polls the bytes waiting, with our own 30 s limit.
' * Never send Print # a number list with "," separators between items: SPEL+ inserts spaces; we
'   build one string, the numbers by FmtStr$ (4 decimals, "." decimal point).
' * CP is a motion option, not a statement parameter with On/Off ("Move P1 CP" = continuous path):
'   "CP Off" once, as a statement, and Move without CP, so every Move ends on the point; Wait then
'   settles before the two grabs.
' * XY(x, y, z, u) sets V and W to 0 (a 6-axis robot would turn its tool): the target is Here with
'   only X, Y, Z replaced (Here :X(x) :Y(y) :Z(z)), which keeps U, V, W, the hand and the local.
' * One statement per line: ":" is kept for point expressions (Here :X(x)).

Global String gReply$
Global Real gVal(10)
Global Integer gCount

Function CalCollect
    Real x, y, z
    String cmd$, token$

    token$ = "change-me-eyetohand"   ' the vision side's token (serve --token-file / EYETOHAND_TOKEN)
    SetNet #201, "192.168.0.10", 5000, LF, NONE, 0
    OpenNet #201 As Client
    WaitNet #201, 10
    If TW Then
        Print "eyetohand: cannot connect to the vision PC"
        Exit Function
    EndIf
    CP Off
    ' the first line: AUTH <token>; a wrong token is answered ERR send ... (code -14) and closed
    If Not Cmd("AUTH " + token$) Then
        ' InStr: the position of the text, 1 at the start (SPEL+ Language Reference)
        If InStr(gReply$, "ERR send") = 1 Then gReply$ = "the vision PC refused the token (AUTH): set token$"
        GoTo Fail
    EndIf

    If Not Cmd("CAL BEGIN cell1,grid:5x5,0,570,70,650,150") Then GoTo Fail

    Do
        If Not Cmd("CAL NEXT") Then GoTo Fail
        If gReply$ = "OK DONE" Then Exit Do
        If gCount <> 3 Then GoTo Fail
        x = gVal(0)
        y = gVal(1)
        z = gVal(2)
        Move Here :X(x) :Y(y) :Z(z)   ' U, V, W kept; ends on the point (CP Off)
        Wait 0.5
        cmd$ = "CAL POINT " + Fmt$(x) + "," + Fmt$(y) + "," + Fmt$(z)
        If Not Cmd(cmd$) Then
            If InStr(gReply$, "ERR moving") = 1 Then
                Wait 1.0
                If Not Cmd(cmd$) Then
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
        gCount = ParseStr(Mid$(gReply$, 4, Len(gReply$) - 3), tok$(), ",")
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
