' eyetohand pick loop for Epson robots (SPEL+, RC700/RC90 with EPSON RC+ 7): LOCATE the round
' parts, pick each one, again. UNTESTED on a controller: no Epson controller here (its exchange with
' the real server is replayed by tests/test_pick_programs.py). Read examples/robots/README.md first.
'
' Vision side: eyetohand serve --tcp 0.0.0.0:5000 --camera URI --calibration cell1 --token-file FILE
'   (the first line: AUTH <token>, token$ below, as in EyetohandCollect.prg; a wrong token stops it)
'   LOCATE 8,12  -> OK <count>,<outside>   (parts outside the calibrated region: only counted)
'   LOCATE NEXT  -> OK <x>,<y>,<z>,<rz>,<sigma>   or OK DONE when every part is handed out
' Controller set-up as for EyetohandCollect.prg (port #201, Terminate = LF).
'
' Manual references: "EPSON RC+ 7.0 SPEL+ Language Reference", by statement/function name
' (SetNet, OpenNet, WaitNet, TW, ChkNet, Print #, Line Input #, CloseNet, CP, Move, Here, point
' expressions with :X :Y :Z, Tool, On, Off, Wait, ParseStr, Val, InStr, Left$, Right$, Mid$, Len).
'
' Traps handled here (as in EyetohandCollect.prg): LF terminator, our own timeout with ChkNet,
' one string per Print #, "CP Off" once and Move without CP (every Move ends on the point), Here with
' only X, Y, Z replaced (keeps U, V, W). Also:
' * the robot must be out of the camera's view during LOCATE: it goes to P1 (clear) first.
' * no pick outside the calibrated region: the server never hands such a part out; a part whose
'   sigma is above MAX_SIGMA (or unknown, -1) is skipped.
' * Tool 1 is the gripper (its TCP: the point the calibration's x, y, z are for); TOOL_DZ the tool
'   offset along z (where the gripper closes, from the part's top), APPROACH the approach height.

Global String gReply$
Global Real gVal(10)
Global Integer gCount

Function PickLoop
    Real x, y, z, sigma
    Real APPROACH, TOOL_DZ, MAX_SIGMA
    String token$

    APPROACH = 50
    TOOL_DZ = -2
    MAX_SIGMA = 0.2
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
    Tool 1

    Do
        Move P1   ' clear of the camera's view
        If Not Cmd("LOCATE 8,12") Then GoTo Fail
        If gCount <> 2 Then GoTo Fail
        If gVal(0) = 0 Then Wait 1.0
        Do
            If Not Cmd("LOCATE NEXT") Then GoTo Fail
            If gReply$ = "OK DONE" Then Exit Do
            If gCount <> 5 Then GoTo Fail
            x = gVal(0)
            y = gVal(1)
            z = gVal(2)
            sigma = gVal(4)
            If sigma < 0 Or sigma > MAX_SIGMA Then
                Print "eyetohand: part skipped: ", gReply$
            Else
                Move Here :X(x) :Y(y) :Z(z + TOOL_DZ + APPROACH)
                Move Here :X(x) :Y(y) :Z(z + TOOL_DZ)
                On 8   ' close the gripper
                Wait 0.3
                Move Here :X(x) :Y(y) :Z(z + TOOL_DZ + APPROACH)
                Move P2   ' drop
                Off 8
                Wait 0.3
            EndIf
        Loop
    Loop
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
